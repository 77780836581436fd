"""Evaluation metrics on top of :mod:`macsplat_cli.metrics`: masked image metrics (two
conventions), pose AUC, depth and focal errors.

**Image metrics** (:func:`image_metrics`), images in [0, 1] ``[H, W, 3]``, mask ``[H, W]``:

* default ("standard") convention: ``psnr``/``ssim`` over the whole image;
  ``psnr_masked`` is the PSNR of the per-channel mean squared error over the mask pixels
  (sum of squared errors / (3 · mask pixels)); ``ssim_masked`` is the SSIM map (Gaussian
  window 11, σ 1.5, see :func:`macsplat_cli.metrics.ssim`) averaged over the mask.
* ``splatt3r=True`` reproduces Splatt3R's test code (reference notes §5): both images are
  first multiplied by the mask (outside pixels black in both); ``psnr``/``ssim`` are then
  taken over the whole masked images (the paper's plain numbers); ``psnr_masked`` divides
  the squared error *summed over the three channels* by the number of mask pixels, i.e.
  three times the per-channel error: ``10·log10(3) ≈ 4.77 dB`` below the standard masked
  PSNR (the paper's parenthesised numbers). ``ssim_masked`` is not reported (the paper
  prints "–"). Not reproduced: Splatt3R's per-batch PSNR (from the MSE of 12 images,
  averaged over batches; here every image gets its own PSNR, averaged), and skimage's
  sample covariance in SSIM (here population statistics: a factor 121/120 on the
  variances).

In both conventions ``psnr_masked_rgbsum`` is the PSNR of the squared error summed over the three channels and
divided by the mask pixels (Splatt3R's masked PSNR; ``psnr_masked`` − 4.77 dB in the standard one), so that the two
formulas stand side by side.

**LPIPS** (with user-supplied VGG and LPIPS weights, ``--lpips-weights``): ``lpips`` over the whole image (over the
masked images in the Splatt3R convention) and ``lpips_masked``, the per-pixel LPIPS of the masked images averaged
over the mask (the MAC-Splat release's masked LPIPS).

**Pose AUC** (:func:`pose_auc`): the pose error of a pair is ``max(rotation error,
translation-direction error)``; a failed reconstruction counts as 180°. AUC@τ is the area
under the recall-vs-error curve up to τ, normalised by τ, with the curve drawn through
``(0, 0)`` and the sorted errors and integrated by trapezoids — the convention of
SuperGlue's ``pose_auc`` used across the matching literature.

**Depth** (:func:`depth_metrics`): AbsRel = mean ``|d − d*| / d*`` and δ<1.25 = fraction
with ``max(d/d*, d*/d) < 1.25``, over pixels where both the estimate ``d`` and the ground
truth ``d*`` are positive, after multiplying ``d`` by ``scale``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from ..metrics import psnr, ssim_map

__all__ = [
    "AUC_THRESHOLDS_DEG",
    "depth_metrics",
    "image_metrics",
    "pose_auc",
    "pose_error_deg",
    "splatt3r_psnr",
    "ssim_means",
]

AUC_THRESHOLDS_DEG = (5.0, 10.0, 20.0)
FAILED_POSE_ERROR_DEG = 180.0


def _arr(x: object) -> np.ndarray:
    a = x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)
    return a.astype(np.float64)


def splatt3r_psnr(pred: np.ndarray, target: np.ndarray, mask: np.ndarray, *, average_over_mask: bool) -> float:
    """Splatt3R's PSNR of one image: both images masked, then whole-image or channel-summed mask MSE.

    Args:
        pred: rendered image. [H, W, 3]
        target: ground truth. [H, W, 3]
        mask: visibility mask. [H, W]
        average_over_mask: ``False``: MSE over all pixels and channels of the masked images;
            ``True``: squared error summed over channels and pixels, divided by the mask
            pixel count (3× the per-channel MSE).
    """
    m = _arr(mask).astype(bool)
    err = ((_arr(pred) - _arr(target)) * m[..., None]) ** 2
    if average_over_mask:
        n = int(m.sum())
        if n == 0:
            return math.nan
        mse = float(err.sum()) / n
    else:
        mse = float(err.mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


SSIM_WINDOW, SSIM_SIGMA = 11, 1.5


def ssim_means(pred: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> tuple[float, float]:
    """Mean SSIM over the image and over the mask, from one float32 SSIM map. [H, W, 3], mask [H, W]

    Returns:
        ``(ssim, ssim_masked)``; the second is NaN without a mask or when the mask is empty
        inside the region where the window fits.
    """
    p = torch.from_numpy(np.ascontiguousarray(pred, np.float32))
    t = torch.from_numpy(np.ascontiguousarray(target, np.float32))
    smap = ssim_map(p, t, window=SSIM_WINDOW, sigma=SSIM_SIGMA).double().numpy()
    masked = math.nan
    if mask is not None:
        pad = SSIM_WINDOW // 2
        m = np.asarray(mask, bool)[pad : pad + smap.shape[0], pad : pad + smap.shape[1]]
        masked = float(smap[m].mean()) if m.any() else math.nan
    return float(smap.mean()), masked


def image_metrics(
    pred: np.ndarray,  # [H, W, 3]
    target: np.ndarray,  # [H, W, 3]
    mask: np.ndarray | None = None,  # [H, W]
    *,
    splatt3r: bool = False,
    lpips: torch.nn.Module | None = None,
) -> dict[str, float]:
    """PSNR and SSIM of a rendered view, whole-image and over the visibility mask (module docstring).

    Args:
        lpips: an LPIPS model (:func:`macsplat_cli.lpips.load_lpips`): adds ``lpips``, over the
            whole image (Splatt3R convention: over the masked images).

    Returns:
        ``psnr``, ``ssim``, and with a mask ``psnr_masked``, ``ssim_masked`` (NaN in the
        Splatt3R convention) and ``mask_fraction``; ``lpips`` with an LPIPS model.
    """
    p = np.clip(_arr(pred), 0.0, 1.0)
    t = _arr(target)
    out: dict[str, float] = {}
    if lpips is not None:
        out.update(_lpips(p, t, mask, lpips, splatt3r))
    if mask is None:
        out["psnr"], out["ssim"] = psnr(p, t), ssim_means(p, t)[0]
        return out
    m = _arr(mask).astype(bool)
    out["mask_fraction"] = float(m.mean())
    if splatt3r:
        pm, tm = p * m[..., None], t * m[..., None]
        out["psnr"] = splatt3r_psnr(p, t, m, average_over_mask=False)
        out["ssim"] = ssim_means(pm, tm)[0]
        out["psnr_masked"] = splatt3r_psnr(p, t, m, average_over_mask=True)
        out["ssim_masked"] = math.nan
    else:
        out["psnr"], out["psnr_masked"] = psnr(p, t), psnr(p, t, m)
        out["ssim"], out["ssim_masked"] = ssim_means(p, t, m)
    out["psnr_masked_rgbsum"] = splatt3r_psnr(p, t, m, average_over_mask=True)
    return out


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, np.float32))


def _lpips(
    p: np.ndarray, t: np.ndarray, mask: np.ndarray | None, lpips: torch.nn.Module, splatt3r: bool
) -> dict[str, float]:
    """``lpips`` over the whole image (over the masked images in the Splatt3R convention) and, with a mask,
    ``lpips_masked``: the per-pixel LPIPS of the masked images averaged over the mask (the MAC-Splat release's
    masked LPIPS)."""
    out: dict[str, float] = {}
    m = _arr(mask).astype(bool) if mask is not None else None
    with torch.no_grad():
        if m is not None:
            pm, tm = p * m[..., None], t * m[..., None]
            out["lpips"] = float(lpips(_t(pm), _t(tm))) if splatt3r else float(lpips(_t(p), _t(t)))
            spatial = getattr(lpips, "spatial", None)  # LPIPS's per-pixel map; another module may have none
            if m.any() and spatial is not None:
                dmap = spatial(_t(pm), _t(tm)).double().numpy()
                out["lpips_masked"] = float(dmap[m].mean())
        else:
            out["lpips"] = float(lpips(_t(p), _t(t)))
    return out


def pose_error_deg(rotation_error: float, translation_error: float) -> float:
    """``max(rotation, translation-direction)`` error; NaN counts as a failure (180°)."""
    errs = [e if math.isfinite(e) else FAILED_POSE_ERROR_DEG for e in (rotation_error, translation_error)]
    return max(errs)


def pose_auc(errors_deg: Sequence[float], thresholds: Sequence[float] = AUC_THRESHOLDS_DEG) -> dict[str, float]:
    """Area under the pose-recall curve up to each threshold, normalised to [0, 1] (module docstring).

    Args:
        errors_deg: one pose error per pair (failures as 180°; NaN is read as 180°).
        thresholds: the thresholds τ in degrees.

    Returns:
        ``{"auc@5": …, "auc@10": …, "auc@20": …}`` (keys from ``thresholds``); NaN when empty.
    """
    keys = [f"auc@{t:g}" for t in thresholds]
    if len(errors_deg) == 0:
        return {k: math.nan for k in keys}
    e = np.sort(np.nan_to_num(np.asarray(errors_deg, np.float64), nan=FAILED_POSE_ERROR_DEG))
    recall = np.arange(1, len(e) + 1) / len(e)
    e = np.concatenate([[0.0], e])
    recall = np.concatenate([[0.0], recall])
    out = {}
    for key, t in zip(keys, thresholds):
        last = int(np.searchsorted(e, t))
        r = np.concatenate([recall[:last], [recall[last - 1]]])
        x = np.concatenate([e[:last], [t]])
        out[key] = float(np.sum((x[1:] - x[:-1]) * (r[1:] + r[:-1]) / 2.0) / t)
    return out


def depth_metrics(pred: np.ndarray, gt: np.ndarray, scale: float = 1.0) -> dict[str, float]:
    """AbsRel and δ<1.25 of an estimated depth map against ground truth, and how much of it was estimated.

    Args:
        pred: estimated depth (0 = none). [H, W]
        gt: ground-truth depth (0 = none), same size. [H, W]
        scale: factor applied to ``pred`` first (e.g. relative → metric).

    Returns:
        ``absrel``, ``delta1``, ``absrel_median`` (after per-image median scaling) and
        ``completeness`` (fraction of ground-truth pixels with an estimate); NaN when no
        pixel has both.
    """
    d, g = _arr(pred) * scale, _arr(gt)
    if d.shape != g.shape:
        raise ValueError(f"depth maps differ in size: {d.shape} vs {g.shape}")
    has_gt = g > 0
    ok = has_gt & (d > 0) & np.isfinite(d)
    out = {"completeness": float(ok.sum() / max(1, has_gt.sum()))}
    if not ok.any():
        return {"absrel": math.nan, "delta1": math.nan, "absrel_median": math.nan, **out}
    dv, gv = d[ok], g[ok]
    ratio = np.maximum(dv / gv, gv / dv)
    dm = dv * (np.median(gv) / np.median(dv))
    return {
        "absrel": float(np.mean(np.abs(dv - gv) / gv)),
        "delta1": float(np.mean(ratio < 1.25)),
        "absrel_median": float(np.mean(np.abs(dm - gv) / gv)),
        **out,
    }
